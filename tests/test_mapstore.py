"""The map layout (mapstore/layout.py), the versioned repository (mapstore/repository.py)
and the map commands (pipeline/cli/map.py), on a small map: 700 x 500 px, chunks 64,
shards 256, cells 16, so that several shards and pyramid levels exist."""

from __future__ import annotations

import csv
import subprocess
import sys
import threading
import time
from datetime import date
from pathlib import Path

import cv2
import numpy as np
import pytest
import zarr
from click.testing import CliRunner

from mapstore.grid import MapGrid
from mapstore.layout import (
    LayoutSpec,
    PoseTable,
    create_floor,
    levels_for,
    read_floor,
    read_poses,
    resize_floor,
    set_version,
    shard_slices,
    write_poses,
)
from mapstore.repository import MapRepository, open_storage
from pipeline.cli import cli
from pipeline.config import load_config

GRID = MapGrid(x0=1.0, y0=2.0, pixel_size=0.01, width=500, height=700)
SPEC = LayoutSpec(chunk_px=64, shard_px=256, layer_cell_px=16, zstd_level=3)
ROOT = Path(__file__).resolve().parents[1]


def _pattern(shape, seed=0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.integers(1, 256, size=shape, dtype=np.uint8)


def _poses(n_a: int = 3, n_b: int = 2, version: int = 1) -> PoseTable:
    n = n_a + n_b
    pose = np.column_stack([np.linspace(1.1, 4.0, n), np.linspace(-1.0, 1.5, n), np.linspace(-3.0, 3.0, n)])
    sigma = np.full((n, 3), np.nan)
    sigma[:n_a] = [1e-3, 2e-3, 1e-4]
    sources = [{"log_id": "log-a", "path": "/data/a", "sha256": "aa" * 32, "frames": n_a, "version": version},
               {"log_id": "log-b", "path": "/data/b", "sha256": "bb" * 32, "frames": n_b, "version": version}]
    return PoseTable(pose, sigma, 0.1 * np.arange(n) + 1.0 / 3.0, [0] * n_a + [1] * n_b,
                     list(range(n_a)) + list(range(n_b)), [version] * n, sources)


def _write_all(root: zarr.Group, grid: MapGrid, seed: int = 0) -> dict[int, np.ndarray]:
    """Fill every level and layer shard by shard (as a renderer owning whole shards would)."""
    info = read_floor(root)
    data = {}
    for k in range(info.levels):
        arr = root[f"floor/{k}"]
        img = _pattern(arr.shape, seed + k)
        for _, (rs, cs) in shard_slices(arr.shape, SPEC.shard_px):
            arr[rs, cs] = img[rs, cs]
        data[k] = img
    layers = root["floor/layers"]
    shape = layers["coverage"].shape
    layers["coverage"][:] = np.arange(np.prod(shape), dtype=np.uint16).reshape(shape) % 7
    tex = np.linspace(0.5, 900.0, int(np.prod(shape)), dtype=np.float32).reshape(shape)
    tex[0, :3] = np.nan
    layers["texture"][:] = tex
    layers["uniqueness"][:] = np.linspace(0.0, 1.0, int(np.prod(shape)), dtype=np.float32).reshape(shape)
    layers["updated"][:] = 1
    return data


REPORT = {"optimization": {"frames": 5, "residual_rms_px": 0.1234}, "links": {"accepted": 7, "candidates": 9}}


def make_mapped(tmp_path: Path) -> dict:
    """A repository with two published versions: v1 (whole map), v2 (one level-0 shard)."""
    url = str(tmp_path / "maprepo")
    repo = MapRepository.create(url)
    s = repo.writable()
    root = zarr.open_group(s.store, mode="a")
    create_floor(root, GRID, SPEC)
    data = _write_all(root, GRID)
    write_poses(root, _poses())
    set_version(root, 1)
    sid1 = repo.commit(s, "publish 1", {"version": 1, "report": REPORT})
    repo.tag(sid1, "v1")

    s = repo.writable()
    root = zarr.open_group(s.store, mode="a")
    patch = np.full((20, 30), 77, np.uint8)
    root["floor/0"][300:320, 260:290] = patch  # inside level-0 shard (1, 1) only
    set_version(root, 2)
    sid2 = repo.commit(s, "publish 2", {"version": 2})
    repo.tag(sid2, "v2")
    return {"url": url, "repo": repo, "sid1": sid1, "sid2": sid2, "data": data}


@pytest.fixture
def mapped(tmp_path: Path) -> dict:
    return make_mapped(tmp_path)


def _root(repo: MapRepository, version: str | None = None) -> zarr.Group:
    return zarr.open_group(repo.readonly(version).store, mode="r")


# --- layout ---------------------------------------------------------------------------------


def test_layout_spec_from_config_and_validation():
    spec = LayoutSpec.from_config(load_config(None)["map"])
    assert spec.shard_px % spec.chunk_px == 0 and spec.shard_px % spec.layer_cell_px == 0
    with pytest.raises(ValueError, match="multiple of map.chunk_px"):
        LayoutSpec(64, 200, 8, 3)
    with pytest.raises(ValueError, match="layer_cell_px"):
        LayoutSpec(64, 256, 24, 3)
    with pytest.raises(ValueError, match="chunk_px"):
        LayoutSpec(0, 256, 16, 3)
    with pytest.raises(ValueError, match="map.zstd_level is missing"):
        LayoutSpec.from_config({"chunk_px": 64, "shard_px": 256, "layer_cell_px": 16})


def test_levels_for():
    assert levels_for(GRID, 64) == 5  # 700 -> 350 -> 175 -> 88 -> 44
    assert levels_for(MapGrid(0, 0, 0.01, 64, 64), 64) == 1
    assert levels_for(MapGrid(0, 0, 0.01, 65, 10), 64) == 2


def test_shard_slices_cover_the_array_once():
    seen = np.zeros((700, 500), int)
    ijs = []
    for ij, (rs, cs) in shard_slices((700, 500), 256):
        seen[rs, cs] += 1
        ijs.append(ij)
    assert (seen == 1).all()
    assert ijs == [(i, j) for i in range(3) for j in range(2)]


def test_create_floor_layout(tmp_path: Path):
    root = zarr.open_group(str(tmp_path / "plain.zarr"), mode="w")  # a plain zarr directory
    create_floor(root, GRID, SPEC, map_id="abc123")
    attrs = root.attrs.asdict()
    assert attrs["format"] == "mosaicmap-map" and attrs["format_version"] == 1 and attrs["map_id"] == "abc123"
    assert attrs["created"].endswith("+00:00")
    floor = root["floor"]
    for k in range(5):
        arr = floor[str(k)]
        assert arr.shape == GRID.level(k).shape and arr.dtype == np.uint8
        assert arr.chunks == (64, 64) and arr.shards == (256, 256) and arr.fill_value == 0
        assert arr.metadata.dimension_names == ("y", "x")
        assert type(arr.compressors[0]).__name__ == "ZstdCodec" and arr.compressors[0].level == 3
    assert "5" not in floor
    assert floor["4"].shape == (44, 32)
    ome = floor.attrs["ome"]
    assert ome["version"] == "0.5"
    ms = ome["multiscales"][0]
    assert [a["name"] for a in ms["axes"]] == ["y", "x"] and ms["axes"][0]["unit"] == "meter"
    assert [d["path"] for d in ms["datasets"]] == ["0", "1", "2", "3", "4"]
    for k, d in enumerate(ms["datasets"]):
        assert d["coordinateTransformations"] == GRID.level(k).ome_transformations()
    meta = floor.attrs["mosaicmap"]
    assert MapGrid.from_attrs(meta["grid"]) == GRID
    assert (meta["chunk_px"], meta["shard_px"], meta["layer_cell_px"], meta["levels"], meta["version"]) == (64, 256, 16, 5, 0)
    cov = floor["layers/coverage"]
    assert cov.shape == GRID.coarsened(16).shape == (44, 32)
    assert cov.chunks == (16, 16) and cov.shards is None and cov.dtype == np.uint16 and cov.fill_value == 0
    for name in ("texture", "uniqueness"):
        arr = floor[f"layers/{name}"]
        assert arr.dtype == np.float32 and np.isnan(arr.fill_value) and arr.shape == (44, 32)
        assert np.isnan(arr[0, 0])
    upd = floor["layers/updated"]
    assert upd.shape == (11, 8) and upd.chunks == (4, 4) and upd.dtype == np.int32
    for name in ("coverage", "texture", "uniqueness", "updated"):
        la = floor[f"layers/{name}"].attrs.asdict()
        assert {"grid", "cell_px", "description", "units"} <= set(la)
        assert MapGrid.from_attrs(la["grid"]) == GRID.coarsened(la["cell_px"])
    info = read_floor(root)
    assert (info.grid, info.spec, info.levels, info.version, info.map_id) == (GRID, SPEC, 5, 0, "abc123")
    assert len(read_poses(root)) == 0
    with pytest.raises(ValueError, match="already holds a floor"):
        create_floor(root, GRID, SPEC)


def test_read_floor_rejects_other_groups(tmp_path: Path):
    root = zarr.open_group(str(tmp_path / "x.zarr"), mode="w")
    with pytest.raises(ValueError, match="not a mosaicmap map"):
        read_floor(root)
    create_floor(root, GRID, SPEC)
    root.attrs["format_version"] = 7
    with pytest.raises(ValueError, match="format version 7"):
        read_floor(root)


def test_poses_round_trip_and_csv(tmp_path: Path):
    root = zarr.open_group(str(tmp_path / "p.zarr"), mode="w")
    create_floor(root, GRID, SPEC)
    table = _poses()
    write_poses(root, table)
    back = read_poses(root)
    for name in ("pose", "sigma", "t", "source", "frame", "version"):
        np.testing.assert_array_equal(getattr(back, name), getattr(table, name))
    assert back.sources == table.sources
    write_poses(root, _poses(1, 1, version=3))  # replaced whole
    assert len(read_poses(root)) == 2 and read_poses(root).version.tolist() == [3, 3]
    write_poses(root, table)
    out = tmp_path / "out" / "poses.csv"
    back.to_csv(out)
    rows = list(csv.DictReader(out.open()))
    assert list(rows[0]) == ["t", "x", "y", "theta", "log_id", "frame", "sigma_x", "sigma_y", "sigma_theta", "version"]
    assert len(rows) == 5 and [r["log_id"] for r in rows] == ["log-a"] * 3 + ["log-b"] * 2
    assert float(rows[1]["t"]) == table.t[1]  # repr floats round-trip exactly
    assert float(rows[4]["theta"]) == table.pose[4, 2]
    assert rows[4]["sigma_x"] == "nan" and float(rows[0]["sigma_y"]) == 2e-3
    with pytest.raises(ValueError, match="source indices"):
        PoseTable(np.zeros((1, 3)), np.zeros((1, 3)), [0.0], [2], [0], [1], [{}])


# --- repository ---------------------------------------------------------------------------


def test_open_storage_and_missing_repo(tmp_path: Path, monkeypatch):
    missing = tmp_path / "nothing"
    with pytest.raises(ValueError, match="no map repository at"):
        MapRepository.open(str(missing))
    assert not missing.exists()  # looking did not create it
    with pytest.raises(ValueError, match="'gs'"):
        open_storage("gs://bucket/map")
    monkeypatch.setenv("AWS_ENDPOINT_URL", "http://localhost:9000")
    assert open_storage("s3://bucket/some/prefix") is not None
    repo = MapRepository.create(f"file://{tmp_path / 'r'}")
    assert (tmp_path / "r" / "refs").is_dir()
    with pytest.raises(ValueError, match="exists already"):
        MapRepository.create(str(tmp_path / "r"))
    assert MapRepository.open_or_create(str(tmp_path / "r")).repo.list_branches() == {"main"}
    assert repo.log()[0]["message"] == "Repository initialized"


def test_commit_tag_and_read_back(mapped):
    repo, sid1, sid2, data = mapped["repo"], mapped["sid1"], mapped["sid2"], mapped["data"]
    assert repo.resolve("v1") == sid1 and repo.resolve(None) == sid2 and repo.resolve("latest") == sid2
    assert repo.resolve(sid1) == sid1 and repo.resolve(sid1.lower()) == sid1
    assert repo.resolve("main") == sid2 and repo.resolve(sid1[:8]) == sid1
    for version in ("v1", sid1):
        root = _root(repo, version)
        np.testing.assert_array_equal(root["floor/0"][...], data[0])
        assert read_floor(root).version == 1
    root = _root(repo)
    assert read_floor(root).version == 2
    level0 = root["floor/0"][...]
    assert (level0[300:320, 260:290] == 77).all()
    mask = np.ones(level0.shape, bool)
    mask[300:320, 260:290] = False
    np.testing.assert_array_equal(level0[mask], data[0][mask])
    np.testing.assert_array_equal(root["floor/3"][...], data[3])
    for bad in ("v9", "ZZZZZZZZZZZZZZZZZZZZ", "AAAAAAAAAAAAAAAAAAAA"):
        with pytest.raises(ValueError, match=f"unknown version '{bad}'"):
            repo.readonly(bad)
    with pytest.raises(ValueError, match="exists already"):
        repo.tag(sid2, "v1")


def test_log_newest_first_with_tags(mapped):
    repo = mapped["repo"]
    repo.tag(mapped["sid2"], "also-v2")
    entries = repo.log()
    assert [e["id"] for e in entries[:2]] == [mapped["sid2"], mapped["sid1"]]
    assert entries[0]["tags"] == ["also-v2", "v2"] and entries[1]["tags"] == ["v1"]
    assert entries[1]["metadata"]["report"] == REPORT and entries[1]["message"] == "publish 1"
    assert entries[0]["written_at"] >= entries[1]["written_at"] and entries[0]["written_at"].endswith("+00:00")
    assert entries[-1]["parent_id"] is None and len(entries) == 3


def test_next_tag(mapped):
    repo = mapped["repo"]
    day = date(2026, 11, 22)
    assert repo.next_tag(today=day) == "v20261122-1"
    repo.tag(mapped["sid1"], "v20261122-1")
    repo.tag(mapped["sid1"], "v20261122-3")
    assert repo.next_tag(today=day) == "v20261122-2"
    assert repo.next_tag("nightly-{date}", today=day) == "nightly-20261122"


def test_rollback_keeps_history(mapped):
    repo, sid1, sid2 = mapped["repo"], mapped["sid1"], mapped["sid2"]
    saved = repo.rollback("v1")
    assert saved.startswith("rollback-from-") and len(saved) == len("rollback-from-20261122T043318")
    assert repo.resolve(None) == sid1 and repo.resolve(saved) == sid2
    assert read_floor(_root(repo)).version == 1
    assert read_floor(_root(repo, saved)).version == 2  # the old tip is still readable
    assert [e["id"] for e in repo.log()][:1] == [sid1]
    with pytest.raises(ValueError, match="already at"):
        repo.rollback("v1")
    second = repo.rollback(saved)  # roll forward again: the rolled-back tip is tagged too
    assert second != saved and repo.resolve(second) == sid1 and repo.resolve(None) == sid2


def test_changed_chunks_lists_only_the_written_shard(mapped):
    repo = mapped["repo"]
    changed = repo.changed_chunks("v1", "v2")
    # a sharded array's diff is per shard (the stored object): rows 300-320 / cols 260-290
    # lie in level-0 shard (1, 1); attribute changes (set_version) list no chunks
    assert changed == {"floor/0": {(1, 1)}}
    first = repo.changed_chunks(repo.log()[-1]["id"], "v1")
    assert first["floor/0"] == {(i, j) for i in range(3) for j in range(2)}
    assert first["floor/4"] == {(0, 0)} and first["floor/layers/updated"] == {(i, j) for i in range(3) for j in range(2)}
    with pytest.raises(ValueError, match="cannot diff"):
        repo.changed_chunks("v2", "v1")


def test_resize_floor_keeps_data_and_updates_metadata(mapped):
    repo, data = mapped["repo"], mapped["data"]
    old = read_floor(_root(repo)).grid
    s_ = old.pixel_size
    new = old.extended(old.x0, old.y0 - 1499 * s_, old.x0 + 899 * s_, old.y0)  # pixel centres
    assert new.shape == (1500, 900) and levels_for(new, 64) == 6
    s = repo.writable()
    root = zarr.open_group(s.store, mode="a")
    with pytest.raises(ValueError, match="origin"):
        resize_floor(root, MapGrid(old.x0 + 0.01, old.y0, old.pixel_size, 900, 1500))
    with pytest.raises(ValueError, match="shrink"):
        resize_floor(root, MapGrid(old.x0, old.y0, old.pixel_size, 400, 1500))
    resize_floor(root, new)
    repo.commit(s, "grow")
    root = _root(repo)
    info = read_floor(root)
    assert info.grid == new and info.levels == 6 and info.version == 2
    for k in range(6):
        assert root[f"floor/{k}"].shape == new.level(k).shape
    level1 = root["floor/1"][...]
    np.testing.assert_array_equal(level1[:350, :250], data[1])
    assert (level1[350:] == 0).all() and (level1[:, 250:] == 0).all()
    assert (root["floor/5"][...] == 0).all()
    ms = root["floor"].attrs["ome"]["multiscales"][0]
    assert [d["path"] for d in ms["datasets"]] == [str(k) for k in range(6)]
    for k, d in enumerate(ms["datasets"]):
        assert d["coordinateTransformations"] == new.level(k).ome_transformations()
    assert ms["datasets"][3]["coordinateTransformations"][1]["translation"] == [-new.level(3).y0, new.level(3).x0]
    cov = root["floor/layers/coverage"]
    assert cov.shape == new.coarsened(16).shape and MapGrid.from_attrs(cov.attrs["grid"]) == new.coarsened(16)
    assert root["floor/layers/updated"].shape == (24, 15)
    assert np.isnan(root["floor/layers/texture"][-1, -1])
    assert read_floor(_root(repo, "v2")).grid == old  # the published version is untouched


def test_commit_lock_blocks_another_process(mapped):
    url = mapped["url"]
    code = ("import sys, time; from mapstore.repository import MapRepository\n"
            f"r = MapRepository.open({url!r})\n"
            "with r.commit_lock():\n"
            "    print('locked', flush=True); sys.stdin.readline()\n")
    proc = subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            text=True, cwd=ROOT)
    try:
        assert proc.stdout.readline().strip() == "locked"
        repo = MapRepository.open(url)
        t0 = time.monotonic()
        with pytest.raises(TimeoutError):
            with repo.commit_lock(timeout_s=0.3):
                pass
        assert time.monotonic() - t0 >= 0.3
        proc.stdin.write("\n")
        proc.stdin.flush()
        assert proc.wait(timeout=20) == 0
        with repo.commit_lock(timeout_s=5):
            pass
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_commit_lock_waits_for_the_holder_and_icechunk_tolerates_the_file(mapped):
    url = mapped["url"]
    holder, waiter = MapRepository.open(url), MapRepository.open(url)
    events = []
    with holder.commit_lock():
        with holder.commit_lock():  # reentrant within one object
            pass

        def wait():
            with waiter.commit_lock():
                events.append(("got", time.monotonic()))

        th = threading.Thread(target=wait)
        th.start()
        time.sleep(0.3)
        assert events == []  # still waiting
        released = time.monotonic()
    th.join(timeout=10)
    assert events and events[0][1] >= released
    assert (Path(url) / ".mosaicmap.lock").exists()
    # icechunk ignores the lock file: commits, reads, and garbage collection work
    s = waiter.writable()
    zarr.open_group(s.store, mode="a")["floor/layers/updated"][0, 0] = 5
    sid = waiter.commit(s, "under the lock")
    from datetime import datetime, timezone
    waiter.repo.garbage_collect(datetime.now(timezone.utc))
    assert _root(MapRepository.open(url), sid)["floor/layers/updated"][0, 0] == 5


# --- CLI ------------------------------------------------------------------------------------


def _run(*args: str):
    return CliRunner().invoke(cli, list(args), catch_exceptions=False)


def test_cli_show(mapped):
    r = _run("show", mapped["url"])
    assert r.exit_code == 0, r.output
    out = r.output
    assert "publish version 2" in out and read_floor(_root(mapped["repo"])).map_id in out
    assert "500 x 700 px (cols x rows) = 5.000 x 7.000 m" in out
    assert "floor/4" in out and "shards 256x256" in out and "zstd(3)" in out
    assert "floor/layers/uniqueness" in out and "5 frames from 2 drive log(s)" in out and "log-b" in out
    assert "v1" in out and mapped["sid1"] in out and "main" in out
    r = _run("show", mapped["url"], "--version", "v1")
    assert r.exit_code == 0 and "publish version 1" in r.output


def test_cli_log_tag_rollback(mapped):
    url, sid1, sid2 = mapped["url"], mapped["sid1"], mapped["sid2"]
    r = _run("log", url)
    assert r.exit_code == 0, r.output
    lines = r.output.splitlines()
    assert lines[0].startswith(sid2[:8]) and "[v2]" in lines[0] and "publish 2" in lines[0]
    assert lines[1].startswith(sid1[:8]) and "5 frames" in lines[1] and "7/9 links" in lines[1]
    assert "residual RMS 0.1234 px" in lines[1] and len(lines) == 3
    r = _run("tag", url, sid1[:8], "golden")
    assert r.exit_code == 0 and f"tagged {sid1} as golden" in r.output
    r = _run("tag", url, sid1, "golden")
    assert r.exit_code == 2 and "golden" in r.output and "exists already" in r.output
    r = _run("rollback", url, "golden")
    assert r.exit_code == 0, r.output
    assert mapped["repo"].resolve(None) == sid1 and "rollback-from-" in r.output
    r = _run("log", url)
    assert r.output.splitlines()[0].startswith(sid1[:8]) and "golden" in r.output.splitlines()[0]
    r = _run("rollback", url, "nope")
    assert r.exit_code == 2 and "'nope'" in r.output
    r = _run("log", url, "--branch", "dev")
    assert r.exit_code == 2 and "'dev'" in r.output


def test_cli_poses(mapped, tmp_path: Path):
    out = tmp_path / "poses.csv"
    r = _run("poses", mapped["url"], "--version", "v1", "--out", str(out))
    assert r.exit_code == 0, r.output
    assert "5 poses from 2 drive log(s)" in r.output
    rows = list(csv.DictReader(out.open()))
    assert len(rows) == 5 and rows[3]["log_id"] == "log-b" and rows[3]["frame"] == "0"


@pytest.mark.parametrize("layer", ["intensity", "coverage", "texture", "uniqueness", "updated"])
def test_cli_quicklook(mapped, tmp_path: Path, layer: str):
    out = tmp_path / f"{layer}.png"
    r = _run("quicklook", mapped["url"], "--layer", layer, "--out", str(out))
    assert r.exit_code == 0, r.output
    img = cv2.imread(str(out), cv2.IMREAD_UNCHANGED)
    assert img is not None
    if layer == "intensity":
        assert img.shape == (700, 500)  # level 0 fits 2048 px
        np.testing.assert_array_equal(img, _root(mapped["repo"])["floor/0"][...])
    elif layer == "updated":
        assert img.shape == (11, 8, 3)
    else:
        assert img.shape == (44, 32, 3)
    if layer == "texture":
        assert (img[0, :3] == 0).all() and img[5, 5].any()  # NaN is black, data is not
    r = _run("quicklook", mapped["url"], "--level", "4", "--out", str(tmp_path / "l4.png"))
    assert r.exit_code == 0 and cv2.imread(str(tmp_path / "l4.png"), cv2.IMREAD_UNCHANGED).shape == (44, 32)


def test_cli_bad_input(mapped, tmp_path: Path):
    missing = str(tmp_path / "no-such-repo")
    for args in (["show", missing], ["log", missing], ["poses", missing, "--out", str(tmp_path / "p.csv")],
                 ["quicklook", missing, "--out", str(tmp_path / "q.png")], ["tag", missing, "v1", "x"],
                 ["rollback", missing, "v1"]):
        r = _run(*args)
        assert r.exit_code == 2, (args, r.output)
        assert missing in r.output and "no map repository" in r.output
        assert len(r.output.strip().splitlines()) == 1
    plain = tmp_path / "plain"
    plain.mkdir()
    r = _run("show", str(plain))
    assert r.exit_code == 2 and str(plain) in r.output
    for args in (["show", mapped["url"], "--version", "v77"],
                 ["poses", mapped["url"], "--version", "v77", "--out", str(tmp_path / "p.csv")],
                 ["quicklook", mapped["url"], "--version", "v77", "--out", str(tmp_path / "q.png")],
                 ["tag", mapped["url"], "v77", "x"]):
        r = _run(*args)
        assert r.exit_code == 2, (args, r.output)
        assert "'v77'" in r.output and mapped["url"] in r.output
    r = _run("quicklook", mapped["url"], "--level", "9", "--out", str(tmp_path / "q.png"))
    assert r.exit_code == 2 and "--level" in r.output and "0..4" in r.output
    empty = MapRepository.create(str(tmp_path / "empty"))
    r = _run("show", empty.url)
    assert r.exit_code == 2 and "not a mosaicmap map" in r.output
